"""What the false alarms of trained runs are, on a simulated root whose scenes can be regenerated.

For each run (a ``radarpc train`` folder) the best weights score a split; every detection that
RADIal's metric counts as a false positive at the confidence threshold gets the cause
:func:`radarpc.eval.false_alarms.false_alarm_causes` finds in the regenerated scene of its frame
(:meth:`radarpc.sim.radial_writer.RadialSimulator.from_root`): a labelled vehicle whose box is off,
a vehicle without a label, a mirror ghost, a moving person or cyclist, static clutter, or nothing.
The regenerated labels of every frame of the split are checked against the root's ``labels.csv``
first, so a root written by another simulator version is refused rather than misread.

::

    python docs/notebook/scripts/false_alarms.py runs/sp_r1 runs/sp1 --split test --threshold 0.2 \\
        --names "spectralpillars-s, radial" "spectralpillars-s, radial-s" \\
        --figure docs/results/figures/detection_false_alarms.png

Prints one JSON object per run. Runs must have been trained on simulated roots (``--data``
overrides the root stored with a run, e.g. after moving it).
"""
from __future__ import annotations

import argparse
import functools
import json
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import DataLoader
from tqdm import tqdm

from radarpc.boxes import ra_to_box_xy
from radarpc.eval.detection import FIXED_THRESHOLD, RANGE_GATE_M
from radarpc.eval.false_alarms import FALSE_ALARM_CAUSES, false_alarm_causes, false_alarm_mask
from radarpc.experiments.radial_detection.evaluation import load_trained
from radarpc.models.targets import decode_detections
from radarpc.sim.radial_labels import labelled_vehicles
from radarpc.sim.radial_writer import RadialSimulator
from radarpc.sim.road import GHOST_OWNER
from radarpc.experiments.radial_detection.task import collate_detection, detection_dataset
from radarpc.viz import save_figure

MOVING_MPS = 0.5  # radial speed over the ground above which an unowned scatterer is a person or cyclist


def run_false_alarms(run: str, split: str, threshold: float, data: str | None = None, points: str | None = None,
                     batch_size: int = 8, progress: bool = True) -> dict:
    """Counts of false alarms by cause for one run (see the module docstring)."""
    cfg, model, key = load_trained(run)
    root = data or key["data"]
    if not isinstance(root, str):          # the scene is regenerated from one simulated root
        raise ValueError(f"{run} was trained on {len(root)} roots ({', '.join(root)}): give --data ROOT "
                         f"--points FILE of one of them")
    sim = RadialSimulator.from_root(root)
    ds = detection_dataset(cfg, root, points or key.get("points"), split)
    loader = DataLoader(ds, batch_size=batch_size, shuffle=False,
                        collate_fn=functools.partial(collate_detection, cfg=cfg))
    counts = np.zeros(len(FALSE_ALARM_CAUSES), np.int64)
    by_range = {(0, 30): 0, (30, 60): 0, (60, 1000): 0}  # of the detection's range (m)
    n_det, n_frames = 0, 0
    with torch.inference_mode():
        for b in tqdm(loader, desc=Path(run).name, disable=not progress):
            dets = decode_detections(model(b.inputs).detection.float(), cfg.targets, threshold=threshold)
            ends = b.label_offset.tolist()
            for f in range(len(dets)):
                num = ds.frame_ids[n_frames + f]
                seq, idx = sim.locate(num)
                lab = b.labels[(ends[f - 1] if f else 0):ends[f]]
                d = dets.frame(f)
                fa = false_alarm_mask(d.score, d.range_m, d.azimuth_deg, lab, threshold=threshold)
                n_det += int((d.score.double() > threshold).sum())
                fr = sim.scene_frame(seq, idx)                # every frame: its labels are checked
                scored = _scored_vehicles(sim, root, num, seq, idx, fr, lab, cfg.difficult)
                if not fa.any():
                    continue
                sc = fr.scatterers
                az, el = torch.deg2rad(sc.azimuth_deg), torch.deg2rad(sc.elevation_deg)
                static_v = -fr.ego_speed_mps * torch.cos(az) * torch.cos(el)
                labelled = torch.isin(fr.owner, torch.as_tensor(scored, dtype=torch.long))
                cause = false_alarm_causes(ra_to_box_xy(d.range_m[fa].double(), d.azimuth_deg[fa].double()),
                                           ra_to_box_xy(sc.range_m, sc.azimuth_deg).double(),
                                           sc.rcs_m2 / sc.range_m ** 4, fr.owner, labelled,
                                           (sc.velocity_mps - static_v).abs() > MOVING_MPS, fr.owner == GHOST_OWNER)
                counts += np.bincount(cause.numpy(), minlength=len(FALSE_ALARM_CAUSES))
                r = d.range_m[fa]
                for (lo, hi) in by_range:
                    by_range[(lo, hi)] += int(((r >= lo) & (r < hi)).sum())
            n_frames += len(dets)
    total = int(counts.sum())
    return {
        "run": str(run), "root": str(root), "split": split, "threshold": threshold, "frames": n_frames,
        "detections_above_threshold": n_det, "false_alarms": total,
        "false_alarms_per_frame": total / max(n_frames, 1),
        "by_cause": {c: int(k) for c, k in zip(FALSE_ALARM_CAUSES, counts)},
        "share_by_cause": {c: (int(k) / total if total else float("nan")) for c, k in zip(FALSE_ALARM_CAUSES, counts)},
        "by_range_m": {f"{lo}-{hi}" if hi < 1000 else f">={lo}": k for (lo, hi), k in by_range.items()},
    }


def _scored_vehicles(sim: RadialSimulator, root: str, num: int, seq: int, idx: int, fr, lab: torch.Tensor,
                     difficult: bool) -> list[int]:
    """Indices into ``fr.vehicles`` of the vehicles whose labels the metric scores (the dataset's
    rows of the frame, inside the range gate), after checking that the regenerated label rows are
    the dataset's: a root written by another simulator version is refused, not misread."""
    rows = sim.label_rows(seq, idx, fr)                    # in the order of labelled_vehicles
    vehicles = labelled_vehicles(sim.cfg, fr)
    kept = [(v, r) for v, r in zip(vehicles.tolist(), rows) if r[10] >= 0 and (difficult or r[16] != 1)]
    want = torch.tensor([[r[10], r[11]] for _, r in kept], dtype=torch.float64).reshape(-1, 2)
    got = lab[:, :2].double()
    # labels.csv holds 4 decimals; match one to one
    close = (torch.cdist(got, want) <= 1e-3 if len(got) and len(want)
             else torch.zeros(len(got), len(want), dtype=torch.bool))
    if len(got) != len(want) or not (close.any(0).all() and close.any(1).all()):
        raise SystemExit(f"{root}: frame {num} regenerated with labels {want.tolist()} but the root lists "
                         f"{got.tolist()}: not written by this simulator version; its scenes cannot be regenerated")
    lo, hi = RANGE_GATE_M
    return [v for v, r in kept if lo <= r[10] <= hi]


def _figure(results: list[dict], names: list[str], path: str) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(9, 0.7 * len(results) + 1.6))
    colours = plt.get_cmap("tab10").colors
    for i, res in enumerate(results):
        left = 0.0
        for k, c in enumerate(FALSE_ALARM_CAUSES):
            w = res["by_cause"][c] / max(res["frames"], 1)
            ax.barh(i, w, left=left, color=colours[k], label=c if i == 0 else None)
            left += w
    ax.set_yticks(range(len(results)), names)
    ax.invert_yaxis()
    ax.set_xlabel(f"false alarms per frame at confidence {results[0]['threshold']:g} ({results[0]['split']} split)")
    ax.legend(loc="lower center", bbox_to_anchor=(0.5, 1.0), ncol=3, fontsize=8, frameon=False)
    fig.tight_layout()
    save_figure(fig, path, dpi=120)
    plt.close(fig)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("runs", nargs="+", help="training run folders (trained on simulated RADIal roots)")
    ap.add_argument("--split", default="test", choices=("train", "val", "test", "all"))
    ap.add_argument("--threshold", type=float, default=FIXED_THRESHOLD, help="confidence threshold (default 0.2)")
    ap.add_argument("--data", help="the simulated root, if not where the runs recorded it")
    ap.add_argument("--points", help="the point store, if not where the runs recorded it")
    ap.add_argument("--figure", help="write a bar chart of false alarms per frame by cause here")
    ap.add_argument("--names", nargs="+", help="the runs' names in the figure (default: their folder names)")
    ap.add_argument("--no-progress", action="store_true")
    args = ap.parse_args(argv)
    if args.names and len(args.names) != len(args.runs):
        ap.error(f"--names needs one name per run ({len(args.runs)}), got {len(args.names)}")
    results = []
    for run in args.runs:
        res = run_false_alarms(run, args.split, args.threshold, args.data, args.points, progress=not args.no_progress)
        print(json.dumps(res))
        results.append(res)
    if args.figure:
        _figure(results, args.names or [Path(r).name for r in args.runs], args.figure)


if __name__ == "__main__":
    main()
