"""radarpc's RADIal targets and metrics beside the official code, on random cases. Prints JSON.

Usage::

    python checks/radial_metrics.py --radial-repo path/to/RADIal [--cases 200] [--seed 0]

Needs a local clone of valeoai/RADIal (``--radial-repo``; ``--radial`` is the same option) and
``shapely`` (which its metrics import); the official modules are imported from the clone, never
copied (``pkbar``, a progress bar it imports but does not use here, is replaced by an empty module
when missing).

* ``metrics``: random frames (0-4 labels at 3-105 m, detections jittered around them plus false
  alarms, raw candidates before NMS) scored by the official ``GetFullMetrics`` (its printed mAP,
  mAR, F1) and by :func:`radarpc.eval.detection.evaluate_detections` after
  :func:`radarpc.models.targets.nms`. Cases where the official code divides by zero (a threshold
  without a true positive) are counted as ``official_failed`` and skipped.
* ``encoder``: the official ``ra_encoder.encode`` / ``decode`` against
  :func:`radarpc.models.targets.encode_targets` / :func:`decode_detections` for labels away from
  the map's edges and from each other (where the official encoder is correct).
* ``losses``: the official ``pixor_loss`` (focal + regression, unweighted) against
  :func:`radarpc.models.losses.focal_loss` / :func:`regression_loss` on random maps, with the
  regression named ``"SmoothL1Loss"`` (smooth L1) and ``"smoothL1Loss"`` (the official config's
  spelling, which falls through to L1) against ``"smooth_l1"`` and ``"l1"``.
* ``freespace``: the official per-frame IoU (rows 0..123) against
  :func:`radarpc.eval.detection.freespace_iou` on random maps.
"""
from __future__ import annotations

import argparse
import contextlib
import importlib.util
import io
import json
import sys
import types
from pathlib import Path

import numpy as np
import torch

from radarpc.boxes import Detections, ra_to_box_xy
from radarpc.eval.detection import evaluate_detections, freespace_iou
from radarpc.models.losses import focal_loss, regression_loss
from radarpc.models.targets import (
    RADIAL_REG_MEAN,
    RADIAL_REG_STD,
    decode_detections,
    encode_targets,
    nms,
)


def _load(path: Path, name: str):
    spec = importlib.util.spec_from_file_location(name, path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _random_frame(rng):
    n = int(rng.integers(0, 5))
    labels = np.stack([rng.uniform(3, 105, n), rng.uniform(-60, 60, n)], 1)
    cand = []
    for r, a in labels:
        for _ in range(int(rng.integers(0, 4))):
            cand.append((r + rng.normal(0, 0.4), a + rng.normal(0, 0.4), rng.uniform(0.3, 1)))
    for _ in range(int(rng.integers(0, 3))):
        cand.append((rng.uniform(3, 105), rng.uniform(-60, 60), rng.uniform(0.05, 1)))
    return labels.astype(np.float32), np.asarray(cand, np.float32).reshape(-1, 3)   # (R, A, C) as decode gives


def _official_full(metrics, preds, labels):
    out = io.StringIO()
    with contextlib.redirect_stdout(out), np.errstate(all="ignore"):
        metrics.GetFullMetrics(preds, labels, range_min=5, range_max=100, IOU_threshold=0.5)
    vals = {}
    for line in out.getvalue().splitlines():
        key, _, v = line.strip().partition(":")
        if key in ("mAP", "mAR", "F1 score"):
            vals[key] = float(v.split()[0])
    return vals


def check_metrics(metrics, rng, n_cases: int) -> dict:
    diffs, failed = [], 0
    for _ in range(n_cases):
        frames = [_random_frame(rng) for _ in range(int(rng.integers(1, 6)))]
        labels = [f[0] for f in frames]
        preds = [f[1] for f in frames]
        try:
            off = _official_full(metrics, preds, labels)
        except ZeroDivisionError:
            failed += 1
            continue
        kept = []
        for p in preds:
            t = torch.from_numpy(p).double()
            k = nms(t[:, 2], ra_to_box_xy(t[:, 0], t[:, 1]), 0.05) if len(p) else torch.zeros(0, dtype=torch.long)
            kept.append(torch.from_numpy(p[k.numpy()][:, [2, 0, 1]]))
        lab = torch.from_numpy(np.concatenate(labels))
        rep = evaluate_detections(Detections.from_frames(kept), lab,
                                  torch.cumsum(torch.tensor([len(x) for x in labels]), 0))
        diffs.append([abs(rep.ap - off["mAP"]), abs(rep.ar - off["mAR"]), abs(rep.f1 - off["F1 score"])])
    d = np.asarray(diffs).reshape(-1, 3)
    return {"cases": n_cases, "official_failed": failed, "compared": len(diffs),
            "max_abs_diff": {"ap": float(d[:, 0].max(initial=0)), "ar": float(d[:, 1].max(initial=0)),
                             "f1": float(d[:, 2].max(initial=0))},
            "cases_differing_over_1e-9": int((d.max(1, initial=0) > 1e-9).sum())}


def check_encoder(encoder_mod, rng, n_cases: int) -> dict:
    enc = encoder_mod.ra_encoder(geometry={"ranges": [512, 896, 1], "resolution": [0.201171875, 0.2], "size": 3},
                                 statistics={"reg_mean": list(RADIAL_REG_MEAN), "reg_std": list(RADIAL_REG_STD)})
    map_diff, dec_diff = 0.0, 0.0
    for _ in range(n_cases):
        # rows 3..120 and columns 3..220, at least 4 cells apart in range: no edge, no overlap
        rows = rng.choice(np.arange(3, 121, 4), size=int(rng.integers(1, 6)), replace=False)
        r = (rows + rng.uniform(0, 1, rows.size)) * 0.8046875
        a = (rng.integers(3, 221, rows.size) - 112 + rng.uniform(0, 1, rows.size)) * 0.8
        lab = np.stack([r, a], 1)
        ref = enc.encode(lab)
        ours = encode_targets(torch.from_numpy(lab)).double().numpy()
        map_diff = max(map_diff, float(np.abs(ref - ours).max()))
        ref_dec = np.asarray(enc.decode(ref, 0.5))                                  # (K, 3) R, A, C
        det = decode_detections(torch.from_numpy(ref).float()[None], threshold=0.5, nms_iou=None)
        ours_dec = det.rows()[:, [1, 2, 0]].double().numpy()
        key = lambda x: np.lexsort((x[:, 1].round(3), x[:, 0].round(3)))
        dec_diff = max(dec_diff, float(np.abs(ref_dec[key(ref_dec)] - ours_dec[key(ours_dec)]).max()))
    return {"cases": n_cases, "max_abs_map_diff": map_diff, "max_abs_decode_diff": dec_diff}


def check_losses(loss_mod, rng, n_cases: int) -> dict:
    worst = {"focal": 0.0, "smooth_l1": 0.0, "l1": 0.0}
    for _ in range(n_cases):
        gen = torch.Generator().manual_seed(int(rng.integers(2 ** 31)))
        target = torch.zeros(2, 3, 128, 224)
        target[:, 0] = (torch.rand(2, 128, 224, generator=gen) < 0.01).float()
        target[:, 1:] = torch.randn(2, 2, 128, 224, generator=gen) * target[:, :1]
        pred = torch.cat([torch.rand(2, 1, 128, 224, generator=gen), torch.randn(2, 2, 128, 224, generator=gen)], 1)
        for name, ours_kind in (("SmoothL1Loss", "smooth_l1"), ("smoothL1Loss", "l1")):
            cls, reg = loss_mod.pixor_loss(pred, target, {"classification": "FocalLoss", "regression": name})
            ours = regression_loss(pred[:, 1:], target[:, 1:], target[:, 0], ours_kind)
            worst[ours_kind] = max(worst[ours_kind], abs(ours.item() - reg.item()) / abs(reg.item()))
        worst["focal"] = max(worst["focal"], abs(focal_loss(pred[:, 0], target[:, 0]).item() - cls.item()) / cls.item())
    return {"cases": n_cases, "max_rel_diff": worst}


def check_freespace(rng, n_cases: int) -> dict:
    diff = 0.0
    for _ in range(n_cases):
        prob = rng.uniform(0, 1, (256, 224)).astype(np.float32)
        label = rng.uniform(0, 1, (256, 224)) < rng.uniform(0.1, 0.9)
        pred = prob[:124].reshape(-1) >= 0.5                                       # RADIal's lines
        lab = label[:124].reshape(-1)
        inter = np.abs(pred * lab).sum()
        ref = inter / (np.sum(lab) + np.sum(pred) - inter)
        ours = freespace_iou(torch.from_numpy(prob)[None], torch.from_numpy(label)[None])[0].item()
        diff = max(diff, abs(ours - ref))
    return {"cases": n_cases, "max_abs_diff": diff}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--radial-repo", "--radial", dest="radial", type=Path, required=True,
                    metavar="RADIAL_REPO", help="local clone of valeoai/RADIal")
    ap.add_argument("--cases", type=int, default=200)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    base = args.radial / "FFTRadNet"
    if not (base / "utils" / "metrics.py").is_file():
        sys.exit(f"{base / 'utils' / 'metrics.py'} not found: pass --radial-repo <local clone of valeoai/RADIal>")
    try:
        import shapely  # noqa: F401
    except ImportError:
        sys.exit("the official metrics need shapely: pip install shapely")
    sys.modules.setdefault("pkbar", types.ModuleType("pkbar"))
    metrics = _load(base / "utils" / "metrics.py", "radial_official_metrics")
    encoder = _load(base / "dataset" / "encoder.py", "radial_official_encoder")
    loss = _load(base / "loss" / "loss.py", "radial_official_loss")
    rng = np.random.default_rng(args.seed)
    print(json.dumps({"metrics": check_metrics(metrics, rng, args.cases),
                      "encoder": check_encoder(encoder, rng, max(args.cases // 4, 1)),
                      "losses": check_losses(loss, rng, max(args.cases // 20, 1)),
                      "freespace": check_freespace(rng, max(args.cases // 4, 1))}, indent=1))


if __name__ == "__main__":
    main()
