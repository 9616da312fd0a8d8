"""Where trained detectors operate against an F1 target: recall and false alarms per threshold.

Reads evaluation JSON files written by ``radarpc evaluate`` (``RUN/eval_<split>.json``) and prints,
for each, :func:`radarpc.eval.operating_points.read_operating_points`: per threshold the recall,
false alarms per label and frame, F1, how many false alarms the target allows at that recall, and
the share of true detections among those scored between the threshold and the next (a
calibration check against what the run's focal loss implies). ``--figure`` draws every file's
thresholds as a curve over the target's region (``q <= (2 / t - 1) r - 1`` in the plane of
recall ``r`` and false alarms per label ``q``)::

    python docs/notebook/scripts/operating_points.py runs/sp/eval_test.json runs/pp/eval_test.json \\
        --names spectralpillars-s pointpillars-s --figure docs/results/figures/detection_operating_points.png

Prints one JSON object per file.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from radarpc.eval.detection import FIXED_THRESHOLD
from radarpc.eval.operating_points import focal_implied_probability, read_operating_points
from radarpc.viz import save_figure


def _at_fixed(res: dict) -> int | None:
    """Index of RADIal's fixed threshold 0.2 among the file's thresholds, if it is one of them."""
    hit = np.flatnonzero(np.isclose(res["thresholds"], FIXED_THRESHOLD, rtol=0, atol=1e-9))
    return int(hit[0]) if len(hit) else None


def _figure(results: list[dict], names: list[str], path: str, q_max: float | None = None) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    target = results[0]["target_f1"]
    fig, (ax, cal) = plt.subplots(1, 2, figsize=(13, 5.2), width_ratios=(1.3, 1))
    r = np.linspace(0, 1, 201)
    if q_max is None:  # threshold 0.1 lies far above the rest; end a little above the 0.2 points
        at_fixed = [res["false_alarms_per_label"][j] for res in results if (j := _at_fixed(res)) is not None]
        q_max = max([0.8] + [1.3 * q for q in at_fixed])
    for f1 in (0.5, 0.6, 0.7, 0.8, 0.9):
        q = (2 / f1 - 1) * r - 1  # the F1 = f1 line
        keep = q >= 0
        ax.plot(r[keep], q[keep], color="0.75", lw=0.8, zorder=0)
        i = np.argmin(np.abs(q - min(q_max * 0.9, q[-1])))
        ax.annotate(f"F1 {f1:g}", (r[i], q[i]), fontsize=7, color="0.45", ha="right", va="bottom")
    edge = np.maximum((2 / target - 1) * r - 1, 0)
    ax.fill_between(r, 0, edge, color="tab:green", alpha=0.15, lw=0, label=f"F1 >= {target:g}")
    colours = plt.get_cmap("tab10").colors
    for k, (res, name) in enumerate(zip(results, names)):
        rec, q = np.asarray(res["recall"]), np.asarray(res["false_alarms_per_label"])
        c = colours[k % 10]
        ax.plot(rec, q, "-o", ms=3, color=c, label=f"{name} ({res['split']})")
        if (j := _at_fixed(res)) is not None:
            ax.plot(rec[j], q[j], "s", ms=8, mfc="none", mec=c)
    ax.plot([], [], "s", ms=8, mfc="none", mec="k", label=f"confidence {FIXED_THRESHOLD:g}")
    ax.set_xlim(0, 1)
    ax.set_ylim(0, q_max)
    ax.set_xlabel("recall (TP / labels)")
    ax.set_ylabel("false alarms per label (FP / labels)")
    ax.set_title("each curve: thresholds 0.1 (top right, may lie above) ... 0.9 (bottom left)", fontsize=9)
    ax.legend(fontsize=8, loc="upper left")

    # right: the share of true detections in each score band against what the loss implies
    grid = np.linspace(0.01, 0.99, 197)
    cal.plot(grid, grid, color="0.6", lw=0.8, ls="--", label="cross-entropy (gamma 0): q = p")
    for gamma in sorted({res["focal_gamma"] for res in results if res["focal_gamma"]}):  # 0: the diagonal
        cal.plot(grid, focal_implied_probability(grid, gamma), color="0.3", lw=1,
                 label=f"focal loss, gamma {gamma:g}: its minimiser")
    for k, (res, name) in enumerate(zip(results, names)):
        th = np.asarray(res["thresholds"])
        hi = np.append(th[1:], 1.0)
        for i, (a, b, prec, n) in enumerate(zip(th, hi, res["band_precision"], res["band_detections"])):
            if n:
                cal.plot([a, b], [prec, prec], color=colours[k % 10], lw=2,
                         label=f"{name} ({res['split']})" if i == 0 else None)
    cal.set_xlim(0, 1)
    cal.set_ylim(0, 1)
    cal.set_xlabel("detection score p (bands between thresholds)")
    cal.set_ylabel("share of true detections in the band; loss: positive rate q")
    cal.set_title("the score a fully trained model gives a cell positive with probability q", fontsize=9)
    cal.legend(fontsize=7, loc="upper left")
    fig.tight_layout()
    save_figure(fig, path, dpi=120)
    plt.close(fig)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("evaluations", nargs="+", help="eval_<split>.json files written by radarpc evaluate")
    ap.add_argument("--target", type=float, default=0.8, help="the F1 to reach (default 0.8)")
    ap.add_argument("--names", nargs="+", help="names in the figure (default: the files' run folders)")
    ap.add_argument("--figure", help="write the operating curves over the target's region here")
    ap.add_argument("--ymax", type=float, help="top of the figure's false-alarm axis (default: above the 0.2 points)")
    args = ap.parse_args(argv)
    if args.names and len(args.names) != len(args.evaluations):
        ap.error(f"--names needs one name per file ({len(args.evaluations)}), got {len(args.names)}")
    if not 0.0 < args.target <= 1.0:
        ap.error(f"--target must be an F1 in (0, 1], got {args.target}")
    results = []
    for path in args.evaluations:
        try:
            res = read_operating_points(path, args.target)
        except ValueError as e:
            raise SystemExit(str(e)) from e
        print(json.dumps(res))
        results.append(res)
    if args.figure:
        _figure(results, args.names or [Path(p).parent.name for p in args.evaluations], args.figure, args.ymax)


if __name__ == "__main__":
    main()
