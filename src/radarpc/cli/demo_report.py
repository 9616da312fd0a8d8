"""``REPORT.md`` of ``radarpc demo``: what each step did and why, the numbers with what they mean and
what good values look like, the two papers' real-data numbers beside them, and every figure.

:mod:`radarpc.cli.demo` calls it with its config, paths and steps (this module imports nothing of
it: no cycle). The report is a function of the demo's outputs and the records of its steps (``steps/*.json``:
seconds, load, time), so that a rerun that reuses every step writes the same report. It reads the
outputs (point stores, ``eval_*.json``, ``log.csv``, ``metrics.json``) and draws one figure of its
own, F1 and freespace mIoU against density (:func:`radarpc.viz.plot_density_curves`).
"""
from __future__ import annotations

import csv
import json
import math
import os
import shlex
from pathlib import Path

__all__ = ["write_report", "fftradnet_note", "LONG_FFTRADNET_FRAMES", "SEED_DETECTION", "SEED_SWEEP", "SEED_MIOU",
           "SEED_COLORADAR"]

# ---- the papers' numbers on real data (the seeds' tables, in percent as printed) ------------------
SEED_DETECTION = {                    # spectral point-cloud paper, Table 3: RADIal's protocol, real RADIal
    "FFTRadNet (RD cube, 3.8 M parameters)": {"ap": 96.8, "ar": 82.2, "f1": 88.9, "re": 0.11, "ae": 0.17},
    "PointPillars (points at 5.7 %, 2.4 M)": {"ap": 88.7, "ar": 93.5, "f1": 91.0, "re": 0.13, "ae": 0.21},
    "SpectralPillars (points at 5.7 %, 2.4 M)": {"ap": 94.3, "ar": 91.5, "f1": 92.9, "re": 0.12, "ae": 0.22},
}
"""Table 3 of the spectral point-cloud paper: AP, AR, F1 (%) over RADIal's confidence sweep, range
(m) and azimuth (deg) errors, on the real RADIal test set after 100 epochs."""

SEED_SWEEP = {                        # Table 2: F1 (%) at confidence 0.2 against density (%)
    "FFTRadNet": ((100.0, 91.5),),
    "SpectralPillars": ((0.7, 74.3), (1.8, 86.0), (5.6, 90.9), (7.2, 91.6), (17.2, 91.3), (32.7, 92.9),
                        (56.4, 93.7)),
    "PointPillars": ((0.7, 81.0), (1.6, 86.0), (5.7, 90.2), (8.8, 90.2), (19.0, 90.5), (30.8, 91.5),
                     (56.2, 92.8)),
}
"""Table 2 of the spectral point-cloud paper: F1 (%) at confidence 0.2 on real RADIal, by density (%)."""

SEED_MIOU = ((100.0, 79.4), (0.5, 78.3), (1.6, 79.6), (5.7, 80.6), (19.0, 80.7), (30.8, 81.0), (56.2, 81.1))
"""Table 1 of the spectral point-cloud paper: freespace mIoU (%) by density (%), the first row the RD
benchmark (FFTRadNet)."""

SEED_COLORADAR = {                    # RaLD paper, Tables 2, 6 and 8: CD / EMD (m) on real ColoRadar
    "OS-CFAR": {"Aspen Lab": (1.175, 1.342), "Hallways": (1.098, 1.387), "ARPG Lab": (1.076, 1.163),
                "Classroom": (1.127, 0.849), "Longboard (outdoor)": (3.565, 4.256),
                "Courtyard (outdoor)": (1.372, 1.541)},
    "RaLD": {"Aspen Lab": (0.339, 0.356), "Hallways": (0.576, 0.515), "ARPG Lab": (0.488, 0.450),
             "Classroom": (0.356, 0.366), "Longboard (outdoor)": (0.866, 1.109),
             "Courtyard (outdoor)": (0.720, 0.796)},
}
"""Chamfer distance and EMD (m) of OS-CFAR and RaLD in the RaLD paper (Table 2: seen indoor scenes;
Table 6: the unseen classroom; Table 8: unseen outdoor scenes after fine-tuning)."""


# ---- formatting ---------------------------------------------------------------------------------
def _num(x, digits: int = 3) -> str:
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "n/a"
    return f"{x:.{digits}f}"


def _pct(fraction: float | None) -> str:
    return "n/a" if fraction is None or not math.isfinite(fraction) else f"{100 * fraction:.3g} %"


def _rel(path: Path, base: Path) -> str:
    return Path(os.path.relpath(path, base)).as_posix()


def _read_json(path: Path) -> dict:
    with open(path, encoding="utf-8") as f:
        return json.load(f)


def _training(run: Path) -> dict:
    """Steps, training seconds and the best validation F1 (its step) from a run's ``log.csv``."""
    with open(run / "log.csv", newline="", encoding="utf-8") as f:
        rows = list(csv.DictReader(f))
    best = max(rows, key=lambda r: float(r["val_f1"]) if r.get("val_f1") not in (None, "", "nan") else -1.0)
    return {"steps": int(rows[-1]["step"]), "seconds": sum(float(r["train_time_s"]) for r in rows),
            "best_f1": float(best["val_f1"]), "best_f1_fixed": float(best["val_f1_fixed"]),
            "best_step": int(best["step"]), "validations": len(rows)}


LONG_FFTRADNET_FRAMES = 8000
"""Training frames (1,000 steps of 8) after which FFTRadNet found vehicles in radarpc's longer
``radial-s`` trainings (docs/results/detection.md)."""


def fftradnet_note(cfg, training: dict, detection_link: str) -> list[str]:
    """The report's paragraph on a FFTRadNet that found nothing, or ``[]``.

    Parameters
    ----------
    cfg : radarpc.cli.demo.DemoConfig
    training : dict
        FFTRadNet's training summary (:func:`_training`): ``steps`` and ``best_f1``.
    detection_link : str
        Markdown of the link to ``docs/results/detection.md``.

    Returns
    -------
    list of str
        Report lines: empty for ``--tiny`` (its numbers mean nothing) and when the best
        validation F1 is above 0; else why, and, below :data:`LONG_FFTRADNET_FRAMES` training
        frames, the options that train it that far.
    """
    if cfg.tiny or training["best_f1"] > 0:
        return []
    text = (f"FFTRadNet found no vehicle on the validation frames in its {training['steps']} steps of "
            f"{cfg.batch_size} frames: it must learn each vehicle's angle from the phases of the receive channels. "
            f"In radarpc's longer trainings on simulated `radial-s` cubes ({detection_link}) its first validation, "
            "after about 1,000 steps of 8 frames, already found vehicles (F1 about 0.25).")
    if training["steps"] * cfg.batch_size < LONG_FFTRADNET_FRAMES:
        text += (" The demo's default budget keeps it under 10 minutes on a CPU; `radarpc demo --fftradnet-steps 1000 "
                 "--batch-size 8` trains it as far (minutes on a GPU, about an hour on 2 CPU cores; expected to find "
                 "vehicles; not measured with the demo's few hundred training frames).")
    return ["", text]


def _docs_link(name: str, report_dir: Path) -> str:
    """``docs/results/NAME`` as a link when this radarpc runs from its source tree, else its name."""
    docs = Path(__file__).resolve().parents[3] / "docs" / "results"
    text = f"docs/results/{name}"
    return f"[`{text}`]({_rel(docs / name, report_dir)})" if (docs / name).is_file() else f"`{text}`"


# ---- the figure the report draws ----------------------------------------------------------------
def _density_figure(cfg, paths, stores: dict, evals: dict, out: Path) -> str:
    """F1 @ 0.2, F1 and freespace mIoU against the achieved density; returns its caption."""
    from radarpc import __version__
    from radarpc.eval.curves import DensityCurve, normalized_auc
    from radarpc.viz import DensityPanel, plot_density_curves

    dens = tuple(stores[d]["achieved"] for d in cfg.densities)
    increasing = all(a < b for a, b in zip(dens, dens[1:]))

    def curve(label: str, values: list) -> DensityCurve | None:
        if any(v is None or not math.isfinite(v) for v in values):
            return None
        auc = normalized_auc(dens, values) if increasing else None
        return DensityCurve(label, dens, tuple((float(v),) for v in values), auc)

    panels = []
    for key, title in (("f1_fixed", "F1 at confidence 0.2"), ("f1", "F1 (RADIal's, over confidences 0.1-0.9)"),
                       ("freespace_miou", "freespace mIoU")):
        curves = [curve(f"SpectralPillars (trained at {100 * cfg.middle:g} %)",
                        [evals["spectralpillars"][d]["metrics"][key] for d in cfg.densities])]
        if key != "freespace_miou":
            curves.append(curve("classical (no learning)", [evals["classical"][d]["metrics"][key]
                                                             for d in cfg.densities]))
        ref = evals["fftradnet"]["metrics"][key]
        refs = (("FFTRadNet on the dense RD cube (100 %)", (float(ref),)),) if ref is not None and math.isfinite(ref) \
            else ()
        panels.append(DensityPanel(ylabel=title.split(" (")[0], title=title,
                                   curves=tuple(c for c in curves if c is not None), references=refs))
    name = "simulated" if cfg.data is None else Path(cfg.data).name
    plot_density_curves(panels, out, title=f"radarpc demo{' --tiny' if cfg.tiny else ''}: test split of the "
                                            f"{name} RADIal root, one run per model",
                        footer=f"radarpc {__version__}; x: achieved density of each point store; AUC_norm: the "
                               f"curve's mean over the density interval (trapezoids)")
    return ("F1 at confidence 0.2 (left), RADIal's F1 (middle) and freespace mIoU (right) on the test split "
            "against the density of the points: SpectralPillars trained once, scored on each density's points; "
            "the classical detector on the same points; FFTRadNet on the whole RD cube as a dashed line")


# ---- the report ---------------------------------------------------------------------------------
def write_report(cfg, paths, steps: list, *, device: str, frame: int, frame_note: str, configs: dict) -> Path:
    """Write ``REPORT.md`` (and the density figure) from the demo's outputs; return its path.

    Parameters
    ----------
    cfg : radarpc.cli.demo.DemoConfig
    paths : radarpc.cli.demo.DemoPaths
    steps : list of radarpc.cli.demo.DemoStep
        Every step, run or reused, in order, each with its record.
    device : str
        The torch device the steps ran on.
    frame, frame_note : int, str
        The frame the figures draw and why it was chosen.
    configs : dict
        The two trainings' experiment configs (``"spectralpillars"``, ``"fftradnet"``).
    """
    import torch

    from radarpc import __version__
    from radarpc.cli.text import plural
    from radarpc.config import load_yaml_mapping
    from radarpc.data.pointstore import PointStore
    from radarpc.data.summary import summarize_radial
    from radarpc.io import atomic_write
    from radarpc.machine import cpu_model

    out = paths.out
    report = out / "REPORT.md"

    # ---- what the steps produced ----
    stores = {}
    for d in cfg.densities:
        ps = PointStore(paths.store(d))
        m = ps.metadata
        stores[d] = {"tau": m.tau, "achieved": m.achieved_density, "peaks": m.peak_density, "frames": len(ps),
                     "points": float(ps.frame_table.n_points.mean()) if len(ps) else 0.0}
    evals = {"spectralpillars": {d: _read_json(paths.run("spectralpillars") / f"{paths.eval_stem(d)}.json")
                                 for d in cfg.densities},
             "fftradnet": _read_json(paths.run("fftradnet") / f"{paths.eval_stem(None)}.json"),
             "classical": {d: _read_json(paths.classical(d) / "eval_test_easy.json") for d in cfg.densities}}
    training = {m: _training(paths.run(m)) for m in ("spectralpillars", "fftradnet")}
    summary = summarize_radial(paths.radial_root)
    colo = _read_json(paths.oscfar / "metrics.json")
    oscfar_cfg = load_yaml_mapping(paths.oscfar / "config.yaml")
    figure_caption = _density_figure(cfg, paths, stores, evals, paths.density_figure)

    records = [s.record for s in steps]
    seconds = sum(r["seconds"] for r in records)
    cpu = sum(r.get("cpu_seconds", 0.0) for r in records)
    loads = [r["load_1min"] for r in records if r.get("load_1min") is not None]
    finished = max(r["finished_utc"] for r in records)
    first = min(r["finished_utc"] for r in records)
    ev_sp = evals["spectralpillars"]
    ev_mid = ev_sp[cfg.middle]
    n_test_labels, n_test_frames = ev_mid["metrics"]["n_labels"], ev_mid["metrics"]["n_frames"]
    data_name = "simulated" if cfg.data is None else "given (`--data`)"
    rel = lambda p: _rel(p, out)                                       # noqa: E731

    L: list[str] = ["# radarpc demo report", ""]
    if cfg.tiny:
        L += ["> **`--tiny`**: toy sizes (a handful of frames, models trained for a few steps). Every step of the "
              "real demo ran, but the numbers below mean nothing; run `radarpc demo` for numbers with a meaning.",
              ""]
    L += [
        "radarpc carries two radar papers on one signal-processing core. This demo ran both pipelines end to "
        "end, each step a `radarpc` command you can run yourself:", "",
        "1. **Spectral point clouds** (the spectral point-cloud paper): an automotive radar's range-Doppler "
        "spectrum is reduced to a point cloud whose size (its *density*) a CFAR threshold sets; a point "
        "detector (SpectralPillars) trained on the points is compared with a detector that reads the whole "
        "spectrum (FFTRadNet), at several densities.",
        "2. **Radar point clouds against LiDAR** (the RaLD paper): the classical radar point cloud (OS-CFAR) "
        "of an indoor/outdoor radar is scored against the LiDAR scan of the same moment, the baseline RaLD's "
        "learned, dense clouds are measured against.", "",
        f"radarpc {__version__}, torch {torch.__version__}, device `{device}`, {torch.get_num_threads()} threads, "
        f"{cpu_model()}. Steps finished between {first} and {finished}; together {seconds:.0f} s ({cpu:.0f} s of CPU)"
        + (f", the 1-minute load average at their starts {min(loads):.1f}-{max(loads):.1f} on "
           f"{os.cpu_count()} logical CPUs (times grow with the load)" if loads else "") + ".", "",
        "## The steps", "",
        "Each step's record is in `steps/` (command, seconds, load): a rerun of `radarpc demo` with the same "
        "settings reuses the finished steps. Seconds are wall time; CPU seconds add up the demo's threads "
        "(about twice the wall time on 2 idle cores; far less when other jobs share the cores). The load is "
        "the 1-minute load average as the step started.", "",
        "| # | step | seconds | CPU seconds | load at start |", "|---|---|---:|---:|---:|",
    ]
    L += [f"| {k} | {s.name} | {s.record['seconds']:.1f} | {_num(s.record.get('cpu_seconds'), 1)} | "
          f"{_num(s.record.get('load_1min'), 2)} |" for k, s in enumerate(steps, 1)]
    L += ["", "What each did and why:", ""]
    for k, s in enumerate(steps, 1):
        L += [f"{k}. **{s.name}**: {s.why}", f"   `radarpc {shlex.join(s.record['argv'])}`"]   # as it ran

    # ---- part 1 ----
    sp_cfg, fft_cfg = configs["spectralpillars"], configs["fftradnet"]
    mid = cfg.middle
    L += ["", "## Part 1: spectral point clouds and vehicle detection", "", "### The data", "",
          f"The {data_name} RADIal root `{rel(paths.radial_root)}`: sensor `{summary.sensor.name}` "
          f"({summary.sensor.n_range} range x {summary.sensor.n_doppler} Doppler bins x {summary.sensor.n_rx} "
          f"receivers, {summary.sensor.n_tx} transmitters sharing the Doppler axis by DDMA), {summary.n_frames} "
          f"frames in {summary.n_sequences} sequences split by sequence into "
          + ", ".join(f"{k} {v}" for k, v in summary.split_frames.items())
          + f" frames; {summary.n_vehicles} labelled vehicles ({summary.n_difficult} marked `Difficult`), "
          f"{summary.n_empty_frames} frames without any. The test split holds {n_test_frames} frames with "
          f"{n_test_labels} vehicles to find in RADIal's easy mode (below).", "",
          f"![frame {frame}: RD spectrum, CFAR envelope, points]({rel(out / 'frame.png')})", "",
          f"`frame.png`: frame {frame}, {frame_note}. (a) The radar measures, for every range and radial velocity "
          "(Doppler) cell, a complex value per receiver: the *RD spectrum*, drawn as its magnitude summed over "
          "receivers in dB. (b) Each transmitter's echo appears at its own Doppler offset (DDMA); summing those "
          "replicas gives the *envelope* E(r, l), on which CFAR (constant false-alarm rate) estimates the local "
          "noise around each cell from a 9 x 9 window outside a 3 x 3 guard and keeps the cells whose power "
          "exceeds tau times that noise (crosses). (c) Each kept cell becomes a point: its antenna snapshot is "
          "beamformed into an azimuth and elevation, so the point has a position, a radial velocity and an "
          "amplitude; the black boxes are the labelled vehicles.", "",
          "### Density and tau", "",
          "**Density** is the share of RD cells a point cloud keeps: |S| / (N_r N_D), with S the cells kept (here "
          "the CFAR cells and their 3 x 3 neighbourhoods, `rd3`) and N_r N_D all range-Doppler cells. RADIal's "
          "own point clouds keep 5.7 %; the paper sweeps 0.5-56 %. **tau** is the CFAR threshold that sets it: "
          "a linear signal-to-noise ratio (10 log10 tau in dB), one value per store, calibrated on the training "
          "frames so that their mean density hits the target. A higher tau keeps fewer, stronger cells.", "",
          "| store | target density | tau (linear, dB) | achieved density | CFAR peaks alone | points per frame |",
          "|---|---:|---:|---:|---:|---:|"]
    for d in cfg.densities:
        s = stores[d]
        tau = "n/a" if s["tau"] is None else f"{s['tau']:.3g} ({10 * math.log10(s['tau']):.1f} dB)"
        L.append(f"| `{rel(paths.store(d))}`{' (trains)' if d == mid else ''} | {_pct(d)} | {tau} | "
                 f"{_pct(s['achieved'])} | {_pct(s['peaks'])} | {s['points']:.0f} |")
    L += ["", "### The two detectors and their training", "",
          "Both predict RADIal's 128 x 224 range-azimuth map of vehicle probability (and box offsets) and a "
          "freespace map, with the same heads, so that only the input differs. Each trained for a fixed number of "
          "optimizer steps from the recipe of `configs/detection/*-easy.yaml` (cross-entropy, without RADIal's "
          "`Difficult` labels); the weights of the best validation F1 are the ones scored. Configs: "
          f"`{rel(paths.config('spectralpillars'))}`, `{rel(paths.config('fftradnet'))}`.", "",
          "| model | reads | parameters | steps x batch | training time | best validation F1 (@ 0.2) at step |",
          "|---|---|---:|---|---:|---|"]
    for key, c, reads in (("spectralpillars", sp_cfg, f"points at {_pct(mid)} (+ rd3, 32 sectors)"),
                          ("fftradnet", fft_cfg, "the dense RD cube")):
        t = training[key]
        ev = ev_mid if key == "spectralpillars" else evals["fftradnet"]
        L.append(f"| {'SpectralPillars' if key == 'spectralpillars' else 'FFTRadNet'} (`{c.model.variant}`"
                 + (f", overrides {c.model.overrides}" if c.model.overrides else "") + f") | {reads} | "
                 f"{ev['parameters']:,} | {t['steps']} x {c.train.batch_size} | {t['seconds']:.0f} s | "
                 f"{_num(t['best_f1'])} ({_num(t['best_f1_fixed'])}) at {t['best_step']} |")
    L += fftradnet_note(cfg, training["fftradnet"], _docs_link("detection.md", out))
    L += ["", f"![SpectralPillars' learning curve]({rel(paths.run('spectralpillars') / 'figures' / 'learning_curve.png')})",
          "", "### Scores on the test split", "",
          "**The protocol (RADIal's).** Every label and every detection becomes a 4 m x 1.8 m box from above "
          "(the near edge centred on the point); a detection finds a vehicle when the boxes overlap with an "
          "intersection over union (IoU) of at least 0.5. Each detection carries a confidence: at a threshold t, "
          "precision is the share of detections above t that find a vehicle, recall the share of vehicles found. "
          "**AP** and **AR** are their means over t = 0.1, 0.2, ..., 0.9 and **F1** = 2 AP AR / (AP + AR) is "
          "RADIal's summary; **F1 @ 0.2** is precision and recall at the one threshold 0.2 (the paper's density "
          "sweep). Both run from 0 to 1: 1 finds every vehicle without a false alarm. Scored in RADIal's *easy "
          "mode* (its `3-Evaluation.py` default): labels marked `Difficult` are left out; frames without vehicles "
          "stay, so their false alarms count. **Freespace mIoU** is the overlap (intersection over union) of the "
          "predicted and the true drivable area in front of the car, 0-50 m, 1 = perfect. Range and azimuth "
          "errors are those of the matched pairs.", "",
          "| model | input | density | AP | AR | **F1** | P @ 0.2 | R @ 0.2 | **F1 @ 0.2** | range err. (m) | "
          "azimuth err. (deg) | freespace mIoU | frames/s (batch 1) |",
          "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]

    def row(name: str, inp: str, dens: str, ev: dict) -> str:
        m = ev["metrics"]
        fps = ev.get("fps_batch1")
        speed = "not timed" if fps is None or not math.isfinite(fps) else f"{fps:.3g} ({ev['device']})"
        return (f"| {name} | {inp} | {dens} | {_num(m['ap'])} | {_num(m['ar'])} | **{_num(m['f1'])}** | "
                f"{_num(m['precision_fixed'])} | {_num(m['recall_fixed'])} | **{_num(m['f1_fixed'])}** | "
                f"{_num(m['range_error_m'], 2)} | {_num(m['azimuth_error_deg'], 2)} | {_num(m.get('freespace_miou'))} | "
                f"{speed} |")

    for d in cfg.densities:
        L.append(row("SpectralPillars" + (" (its own points)" if d == mid else ""), "points",
                     _pct(stores[d]["achieved"]), ev_sp[d]))
    L.append(row("FFTRadNet", "RD cube", "100 %", evals["fftradnet"]))
    for d in cfg.densities:
        L.append(row("classical", "points", _pct(stores[d]["achieved"]), evals["classical"][d]))
    fig_tag = f"frame{frame:06d}"
    sp_frame = paths.run("spectralpillars") / "figures" / f"{paths.eval_stem(None)}_{fig_tag}.png"
    fft_frame = paths.run("fftradnet") / "figures" / f"{paths.eval_stem(None)}_{fig_tag}.png"
    L += ["", "Minutes of training are far from the end of learning (the trainings behind "
          + _docs_link("detection.md", out) + " take 40-90 minutes): FFTRadNet in particular learns more slowly per "
          "step than the point models, as it must learn each vehicle's angle from the antennas' phases, which the "
          "points get from the beamformer. SpectralPillars trained once, on the middle density; scored on the "
          "other stores it shows how the same detector fares with fewer or more points (the paper trains one "
          "model per density). The classical "
          "detector needs no training: ego speed from the points, the points that move against the ground, "
          "clustered from above, one detection per cluster (its confidence from the cluster's size).", "",
          f"![SpectralPillars on frame {frame}]({rel(sp_frame)})", "",
          f"`{rel(sp_frame)}`: SpectralPillars on frame {frame}, its points from above with the labelled "
          "(green) and predicted (red, confidence >= 0.2) boxes, and its vehicle probability over range and "
          "azimuth.", "",
          f"![FFTRadNet on frame {frame}]({rel(fft_frame)})", "",
          f"![F1 against density]({rel(paths.density_figure)})", "",
          f"`{rel(paths.density_figure)}`: {figure_caption}.", ""]

    # the papers' numbers
    sweep = SEED_SWEEP["SpectralPillars"]

    def nearest(pct: float, table) -> tuple[float, float]:
        return min(table, key=lambda t: abs(math.log(t[0] / pct)))

    L += ["### What good values look like: the paper's real-data numbers", "",
          "**These are the numbers the spectral point-cloud paper reports on the real RADIal dataset** (GPU "
          "training for 50-100 epochs, the full-size sensor, ten runs per configuration for the sweep), beside "
          "this demo's single short runs on simulated data. They say what a trained detector reaches, not what "
          "this demo should: "
          + ("`--tiny` trains for a few steps on 9 frames." if cfg.tiny else
             f"this demo trains for {training['spectralpillars']['steps']} and "
             f"{training['fftradnet']['steps']} steps on {summary.split_frames.get('train', 0)} frames of the "
             f"`{summary.sensor.name}` sensor, minutes on a CPU.")
          + " radarpc's longer trainings on simulated data are in " + _docs_link("detection.md", out)
          + " (pillar models 0.81-0.82 F1 @ 0.2 on `radial` points after 42-54 minutes on 2 cores; "
          "`fftradnet-s` 0.48-0.55 on `radial-s` cubes).", "",
          "| quantity | this demo (simulated) | the paper (real RADIal) |", "|---|---:|---:|"]
    for d in cfg.densities:
        ach = 100 * stores[d]["achieved"]
        sd, sf = nearest(ach, sweep)
        L.append(f"| SpectralPillars F1 @ 0.2 at {ach:.3g} % | {_num(ev_sp[d]['metrics']['f1_fixed'])} | "
                 f"{sf / 100:.3f} at {sd:g} % (Table 2) |")
    L += [f"| FFTRadNet (dense RD) F1 @ 0.2 | {_num(evals['fftradnet']['metrics']['f1_fixed'])} | "
          f"{SEED_SWEEP['FFTRadNet'][0][1] / 100:.3f} (Table 2) |",
          f"| SpectralPillars RADIal F1 on its own points ({_pct(stores[mid]['achieved'])}) | "
          f"{_num(ev_mid['metrics']['f1'])} | "
          f"{SEED_DETECTION['SpectralPillars (points at 5.7 %, 2.4 M)']['f1'] / 100:.3f} at 5.7 % (Table 3) |",
          f"| FFTRadNet RADIal F1 | {_num(evals['fftradnet']['metrics']['f1'])} | "
          f"{SEED_DETECTION['FFTRadNet (RD cube, 3.8 M parameters)']['f1'] / 100:.3f} (Table 3) |"]
    md, mv = nearest(100 * stores[mid]["achieved"], SEED_MIOU[1:])
    L += [f"| freespace mIoU, points at {100 * stores[mid]['achieved']:.3g} % | "
          f"{_num(ev_mid['metrics'].get('freespace_miou'))} | {mv / 100:.3f} at {md:g} % (Table 1) |",
          f"| freespace mIoU, dense RD | {_num(evals['fftradnet']['metrics'].get('freespace_miou'))} | "
          f"{SEED_MIOU[0][1] / 100:.3f} (Table 1) |", "",
          "The paper's full tables (real RADIal):", "",
          "| model (Table 3, RADIal's protocol) | AP | AR | F1 | range err. (m) | azimuth err. (deg) |",
          "|---|---:|---:|---:|---:|---:|"]
    L += [f"| {k} | {v['ap'] / 100:.3f} | {v['ar'] / 100:.3f} | {v['f1'] / 100:.3f} | {v['re']:.2f} | {v['ae']:.2f} |"
          for k, v in SEED_DETECTION.items()]
    L += ["", "| density (Table 2) | " + " | ".join(f"{d:g} %" for d, _ in sweep) + " |",
          "|---|" + "---:|" * len(sweep),
          "| SpectralPillars F1 @ 0.2 | " + " | ".join(f"{f / 100:.3f}" for _, f in sweep) + " |",
          f"| (FFTRadNet, dense: {SEED_SWEEP['FFTRadNet'][0][1] / 100:.3f}) |" + " |" * len(sweep), "",
          "In the paper F1 rises with density and does not fall at high density, SpectralPillars reaches the "
          "dense FFTRadNet at 7.2 %, and point clouds match the RD benchmark's freespace mIoU (0.794) from 1.6 % "
          "on. Whether the simulated data reproduces each finding is the subject of the study "
          "(`radarpc experiment density-sweep`; its results, finding by finding: " + _docs_link("study.md", out)
          + ").", ""]

    # ---- part 2 ----
    ov = colo["overall"]
    how = (oscfar_cfg.get("provenance") or {}).get("how", "")
    scenes = [s.strip() for s in cfg.colo_scenes.split(",") if s.strip()]
    L += ["## Part 2: radar point clouds against LiDAR (ColoRadar)", "",
          f"Simulated ColoRadar runs ({', '.join(scenes)}), scored on the test runs: "
          f"{plural(ov['n_frames'], 'frame')}. "
          "OS-CFAR ranks the cells around each cell of the radar cube and keeps those above the threshold. Its "
          f"setting, {how}: `{json.dumps(oscfar_cfg.get('oscfar', {}), sort_keys=True)}`.", "",
          "**Chamfer distance (CD)**: for each LiDAR point the distance to the nearest radar point, and for "
          "each radar point the distance to the nearest LiDAR point; the two means, averaged (RaLD's definition, "
          "not squared), in metres. **EMD** (earth mover's distance): the mean distance points must travel to turn "
          "one cloud into the other when every point carries the same mass (exact Wasserstein-1 between 2,048 "
          "LiDAR points and up to 2,048 radar points), in metres. Both are 0 for identical clouds and lower is "
          "better; a radar cloud of a few hundred points cannot cover a LiDAR surface of tens of thousands, so EMD "
          "has a floor (about 0.22 m on the simulated scenes of " + _docs_link("coloradar.md", out) + ").", "",
          (paths.oscfar / "metrics.md").read_text(encoding="utf-8").strip(), ""]
    for s in scenes:
        L += [f"![{s}: radar cube, LiDAR, OS-CFAR]({rel(paths.oscfar / 'figures' / f'{s}.png')})", ""]
    L += ["**The RaLD paper's numbers on the real ColoRadar dataset** (CD / EMD in metres; RaLD is the learned "
          "model this demo does not train):", "",
          "| scene (real ColoRadar) | OS-CFAR CD | OS-CFAR EMD | RaLD CD | RaLD EMD |", "|---|---:|---:|---:|---:|"]
    L += [f"| {scene} | {c:.3f} | {e:.3f} | {SEED_COLORADAR['RaLD'][scene][0]:.3f} | "
          f"{SEED_COLORADAR['RaLD'][scene][1]:.3f} |" for scene, (c, e) in SEED_COLORADAR["OS-CFAR"].items()]
    L += ["", f"This demo's OS-CFAR on simulated scenes: CD {_num(ov['chamfer_mean'])} m, EMD {_num(ov['emd_mean'])} "
          "m. The CD is comparable in kind; the EMD is not (the paper publishes neither its EMD implementation nor "
          "its subset sizes); see " + _docs_link("coloradar.md", out) + ".", "",
          "## Further", "",
          "- " + _docs_link("README.md", out) + ": every measured result, with its config and command.",
          "- " + _docs_link("detection.md", out) + ", " + _docs_link("pointcloud.md", out) + ", "
          + _docs_link("coloradar.md", out) + ": the detection models, the point clouds, the ColoRadar side.",
          "- " + _docs_link("study.md", out) + ": the study behind the paper's figures on simulated data (density "
          "sweep, ablations, sparse RD, FPS), finding by finding; run it with `radarpc experiment density-sweep "
          "configs/study/density-sweep.yaml --out runs/sweep`, then `radarpc report runs/sweep`.", "",
          "## Every figure", ""]
    figures = [(f, c) for s in steps for f, c in s.figures] + [(paths.density_figure, figure_caption)]
    L += [f"- `{rel(f)}`: {c}." for f, c in figures]
    text = "\n".join(L) + "\n"
    with atomic_write(report, "w") as f:
        f.write(text)
    return report
