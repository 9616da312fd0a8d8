"""Where trained detectors operate against an F1 target: recall and false alarms per threshold.

RADIal's F1 at one confidence threshold is ``2 TP / (2 TP + FP + FN)``. With ``L = TP + FN``
(the labels, unless two detections hit one), recall ``r = TP / L`` and ``q = FP / L`` false
alarms per label it is

    F1 = 2 r / (1 + r + q),

so a target F1 ``t`` holds exactly where

    q <= (2 / t - 1) r - 1,

a half-plane in the (recall, false alarms per label) plane that needs ``r >= t / (2 - t)`` even
without false alarms (0.667 for t = 0.8) and allows at most ``2 / t - 2`` false alarms per label
at full recall (0.5). This script reads evaluation JSON files written by ``radarpc evaluate``
(``RUN/eval_<split>.json``), prints for each and each threshold the recall, false alarms per label
and frame, F1, how many false alarms the target allows at that recall, and the share of true
detections among those scored between the threshold and the next (a calibration check), and draws
every file's thresholds as a curve over the target's region::

    python benchmarks/operating_points.py runs/sp/eval_test.json runs/pp/eval_test.json \\
        --names spectralpillars-s pointpillars-s --figure docs/results/figures/detection_operating_points.png

Prints one JSON object per file.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from radarpc.eval.detection import FIXED_THRESHOLD
from radarpc.viz import save_figure


def allowed_false_alarms(tp: np.ndarray, fn: np.ndarray, target: float) -> np.ndarray:
    """The most false alarms at which F1 still reaches ``target`` with these hits and misses.

    ``2 TP / (2 TP + FP + FN) >= t`` holds exactly while ``FP <= 2 TP (1 / t - 1) - FN``; in
    terms of ``L = TP + FN``, recall ``r`` and ``q = FP / L``: ``q <= (2 / t - 1) r - 1``.

    Parameters
    ----------
    tp, fn : ndarray
        True positives and missed labels (counts >= 0), broadcastable.
    target : float
        F1 to reach, in (0, 1].

    Returns
    -------
    ndarray
        The whole number of false alarms allowed; -1 where even none would do.
    """
    tp, fn = np.asarray(tp, dtype=np.float64), np.asarray(fn, dtype=np.float64)
    if not 0.0 < target <= 1.0:
        raise ValueError(f"target F1 must be in (0, 1], got {target}")
    if np.any(tp < 0) or np.any(fn < 0):
        raise ValueError("tp and fn must be counts >= 0")
    bound = 2 * tp * (1 / target - 1) - fn
    # the bound is often a whole number (2 TP / t is, for t = 0.8 and even TP) that the float
    # arithmetic leaves a few ulp below; counts are < 2^40, so 1e-6 cannot reach the next one
    return np.maximum(np.floor(bound + 1e-6), -1).astype(np.int64)


def focal_implied_probability(score: np.ndarray, gamma: float) -> np.ndarray:
    """The chance of being positive that a cell has when the focal loss is minimised at ``score``.

    For a cell that is positive with probability ``q``, the expected focal loss
    ``q (1 - p)^gamma (-log p) + (1 - q) p^gamma (-log(1 - p))`` is stationary where
    ``q A(p) + (1 - q) B(p) = 0`` with ``A = d/dp (1 - p)^gamma (-log p) < 0`` and
    ``B = d/dp p^gamma (-log(1 - p)) > 0``, so ``q = B / (B - A)``: the inverse of the score a
    perfectly trained model gives that cell (a property of cells, not of detections after NMS).
    ``gamma = 0`` (cross-entropy) gives ``q = p``; RADIal's ``gamma = 2`` gives ``q = 0.024`` at
    ``p = 0.2``.

    Parameters
    ----------
    score : ndarray
        Scores ``p`` in (0, 1), any shape.
    gamma : float
        Focusing exponent (>= 0).

    Returns
    -------
    ndarray
        ``q`` in (0, 1), the shape of ``score``; increasing in ``p``.
    """
    p = np.asarray(score, dtype=np.float64)
    if gamma < 0:
        raise ValueError(f"gamma must be >= 0, got {gamma}")
    if np.any((p <= 0) | (p >= 1)):
        raise ValueError(f"scores must lie in (0, 1), got {p.min()}..{p.max()}")
    nlog_p, nlog_1mp = -np.log(p), -np.log1p(-p)
    a = -gamma * (1 - p) ** (gamma - 1) * nlog_p - (1 - p) ** gamma / p
    b = gamma * p ** (gamma - 1) * nlog_1mp + p ** gamma / (1 - p)
    return b / (b - a)


def operating_points(evaluation: dict, target: float, gamma: float | None = None) -> dict:
    """Per threshold: recall, false alarms per label and frame, F1, and the target's allowance.

    Parameters
    ----------
    evaluation : dict
        What ``radarpc evaluate`` writes: ``split`` and ``metrics`` with ascending ``thresholds``,
        per-threshold ``tp``, ``fp``, ``fn`` and the split's ``n_frames``.
    target : float
        F1 to reach, in (0, 1].
    gamma : float, optional
        The run's focal exponent; adds the positive rate each threshold stands for under it.

    Returns
    -------
    dict
        Per threshold (lists): ``recall`` ``TP / (TP + FN)``, ``false_alarms_per_label``
        ``FP / (TP + FN)``, ``false_alarms_per_frame``, ``f1``, ``false_alarms``,
        ``allowed_false_alarms`` (-1: the recall alone misses the target), ``band_detections`` and
        ``band_precision`` (detections scored above this threshold and up to the next, and the
        share of them that are true; None for an empty band), ``implied_probability`` (or None).
    """
    m = evaluation["metrics"]
    th = np.asarray(m["thresholds"], dtype=np.float64)
    tp, fp, fn = (np.asarray(m[k], dtype=np.float64) for k in ("tp", "fp", "fn"))
    if not (th.ndim == 1 and tp.shape == fp.shape == fn.shape == th.shape and len(th)):
        raise ValueError(f"thresholds, tp, fp and fn must be lists of one length, got "
                         f"{th.shape}, {tp.shape}, {fp.shape}, {fn.shape}")
    if np.any(np.diff(th) <= 0):
        raise ValueError(f"thresholds must ascend, got {th.tolist()}")
    n_frames = int(m["n_frames"])
    # a detection is kept above a threshold, so TP and FP only fall as it rises
    if np.any(np.diff(tp) > 0) or np.any(np.diff(fp) > 0):
        raise ValueError(f"tp {tp.tolist()} and fp {fp.tolist()} must not rise with the threshold")
    labels = np.maximum(tp + fn, 1)  # RADIal's recall is TP / (TP + FN) at each threshold
    band_tp = tp - np.append(tp[1:], 0)
    band = band_tp + fp - np.append(fp[1:], 0)
    return {
        "split": evaluation["split"],
        "n_frames": n_frames,
        "target_f1": target,
        "thresholds": th.tolist(),
        "recall": (tp / labels).tolist(),
        "false_alarms_per_label": (fp / labels).tolist(),
        "false_alarms_per_frame": (fp / max(n_frames, 1)).tolist(),
        "f1": (2 * tp / np.maximum(2 * tp + fp + fn, 1)).tolist(),
        "false_alarms": fp.astype(int).tolist(),
        "allowed_false_alarms": allowed_false_alarms(tp, fn, target).tolist(),
        # detections kept at threshold k but not at k + 1: scores in (t_k, t_k+1], the last band
        # all above the top threshold
        "band_detections": band.astype(int).tolist(),
        "band_precision": [float(t / n) if n else None for t, n in zip(band_tp, band)],
        "focal_gamma": gamma,
        "implied_probability": None if gamma is None else focal_implied_probability(th, gamma).tolist(),
    }


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
        run_json = Path(path).parent / "run.json"  # the run folder's key, when the file sits in one
        gamma = None
        if run_json.exists():
            try:
                gamma = float(json.loads(run_json.read_text())["experiment"]["loss"]["focal_gamma"])
            except (OSError, json.JSONDecodeError, KeyError, TypeError, ValueError) as e:
                raise SystemExit(f"{run_json}: expected a run folder's run.json with "
                                 f"experiment.loss.focal_gamma: {e!r}") from e
        try:
            res = operating_points(json.loads(Path(path).read_text()), args.target, gamma)
        except (OSError, json.JSONDecodeError, KeyError, TypeError, ValueError) as e:
            raise SystemExit(f"{path}: expected an evaluation JSON written by radarpc evaluate "
                             f"(split, and metrics with ascending thresholds, per-threshold tp, fp, fn, "
                             f"and n_frames): {e!r}") from e
        res["file"] = str(path)
        print(json.dumps(res))
        results.append(res)
    if args.figure:
        _figure(results, args.names or [Path(p).parent.name for p in args.evaluations], args.figure, args.ymax)


if __name__ == "__main__":
    main()
