"""Where a detector operates against an F1 target: recall and false alarms per confidence threshold.

RADIal's F1 at one confidence threshold is ``2 TP / (2 TP + FP + FN)``. With ``L = TP + FN``
(the labels, unless two detections hit one), recall ``r = TP / L`` and ``q = FP / L`` false
alarms per label it is

    F1 = 2 r / (1 + r + q),

so a target F1 ``t`` holds exactly where

    q <= (2 / t - 1) r - 1,

a half-plane in the (recall, false alarms per label) plane that needs ``r >= t / (2 - t)`` even
without false alarms (0.667 for t = 0.8) and allows at most ``2 / t - 2`` false alarms per label
at full recall (0.5).

:func:`operating_points` reads the per-threshold counts of an evaluation (what ``radarpc
evaluate`` writes to ``RUN/eval_<split>.json``) and gives, per threshold, the recall, the false
alarms per label and per frame, F1, how many false alarms the target allows at that recall
(:func:`allowed_false_alarms`), and the share of true detections among those scored between the
threshold and the next: a calibration check against the positive rate the run's focal loss
implies for that score (:func:`focal_implied_probability`). :func:`read_operating_points` does
the same for an evaluation file, with the focal exponent read from the run folder's ``run.json``
beside it.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

__all__ = [
    "allowed_false_alarms",
    "focal_implied_probability",
    "operating_points",
    "read_operating_points",
]


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


def read_operating_points(path: str | Path, target: float = 0.8) -> dict:
    """:func:`operating_points` of an evaluation file written by ``radarpc evaluate``.

    Parameters
    ----------
    path : str or Path
        ``RUN/eval_<split>.json``. When a ``run.json`` lies beside it (the file sits in a run
        folder), the run's focal exponent ``experiment.loss.focal_gamma`` is read from it.
    target : float
        F1 to reach, in (0, 1].

    Returns
    -------
    dict
        :func:`operating_points` with ``file`` (``path`` as given).

    Raises
    ------
    ValueError
        Naming the file: a ``run.json`` without the focal exponent, or an evaluation file that
        cannot be read or lacks the counts; a target outside (0, 1].
    """
    if not 0.0 < target <= 1.0:
        raise ValueError(f"target F1 must be in (0, 1], got {target}")
    run_json = Path(path).parent / "run.json"
    gamma = None
    if run_json.exists():
        try:
            gamma = float(json.loads(run_json.read_text())["experiment"]["loss"]["focal_gamma"])
        except (OSError, json.JSONDecodeError, KeyError, TypeError, ValueError) as e:
            raise ValueError(f"{run_json}: expected a run folder's run.json with "
                             f"experiment.loss.focal_gamma: {e!r}") from e
    try:
        res = operating_points(json.loads(Path(path).read_text()), target, gamma)
    except (OSError, json.JSONDecodeError, KeyError, TypeError, ValueError) as e:
        raise ValueError(f"{path}: expected an evaluation JSON written by radarpc evaluate "
                         f"(split, and metrics with ascending thresholds, per-threshold tp, fp, fn, "
                         f"and n_frames): {e!r}") from e
    res["file"] = str(path)
    return res
