"""Check: does bf16 autocast keep a trained run's decoded detections?

On random weights every cell of the detection map sits near the same probability, so bf16's
rounding moves cells across RADIal's 0.05 candidate threshold and the decoded detections of
``benchmarks/fftradnet_official.py`` cannot tell whether bf16 keeps them. A trained model's map
separates vehicles from the rest; this script runs a trained run's frames on the CPU in fp32 and
under bf16 autocast (the same weights) and prints one JSON object with, over the frames:

* ``by_threshold``: for the decoding threshold 0.05 and each of RADIal's confidence thresholds
  0.1 ... 0.9 (the metrics see only detections above these), the detections above it in each
  precision, those left without a partner in the other (pairs: one to one, nearest first,
  within half a cell: 0.4 m in range and 0.4 deg in azimuth;
  :func:`radarpc.eval.agreement.pair_detections`), and the frames where every detection
  has its partner (``frames_same``);
* ``matched``: over the pairs at 0.05, the largest score, range and azimuth differences;
* ``cells``: the largest logit difference over all cells (``max_logit_diff``) and how many cells
  lie within it of the 0.05 threshold's logit (``cells_in_band``): the cells rounding can move
  across it. A detection near a threshold may be in one precision only for that reason alone.

Usage::

    python docs/notebook/scripts/bf16_detections.py runs/fft --split test [--frames 100] [--threads 2]
"""
from __future__ import annotations

import argparse
import functools
import json
import math

import torch
from torch.utils.data import DataLoader, Subset

from radarpc.eval.agreement import pair_detections
from radarpc.eval.detection import THRESHOLDS as CONFIDENCE_THRESHOLDS
from radarpc.experiments.radial_detection.evaluation import load_trained
from radarpc.machine import cpu_has_native_bf16, cpu_model
from radarpc.boxes import Detections
from radarpc.models.targets import decode_detections
from radarpc.training.loop import autocast_context
from radarpc.experiments.radial_detection.task import DECODE_THRESHOLD, collate_detection, detection_dataset


def _above(d: Detections, t: float) -> Detections:
    """The detections of one frame with score ``> t``, compared in float64 as the metrics do
    (:func:`radarpc.eval.detection.match_frame`)."""
    keep = d.score.double() > t
    return Detections(d.score[keep], d.range_m[keep], d.azimuth_deg[keep], d.offset.new_tensor([int(keep.sum())]))


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("run", help="a training run folder (radarpc train --out)")
    p.add_argument("--split", default="test")
    p.add_argument("--frames", type=int, help="only the split's first N frames")
    p.add_argument("--batch-size", type=int, default=8)
    p.add_argument("--threads", type=int, default=torch.get_num_threads())
    a = p.parse_args(argv)
    torch.set_num_threads(a.threads)
    cfg, model, key = load_trained(a.run, "cpu")
    ds = detection_dataset(cfg, key["data"], key.get("points"), a.split)
    if a.frames is not None:
        ds = Subset(ds, range(min(a.frames, len(ds))))
    loader = DataLoader(ds, batch_size=a.batch_size, shuffle=False,
                        collate_fn=functools.partial(collate_detection, cfg=cfg))
    band_logit = math.log(DECODE_THRESHOLD / (1 - DECODE_THRESHOLD))
    thresholds = (DECODE_THRESHOLD,) + CONFIDENCE_THRESHOLDS
    counts = {t: {"fp32": 0, "bf16": 0, "fp32_unpaired": 0, "bf16_unpaired": 0, "frames_same": 0} for t in thresholds}
    frames = 0
    d_score = d_range = d_az = 0.0
    logit_diffs, fp32_logits = [], []
    cpu = torch.device("cpu")
    with torch.inference_mode():
        for batch in loader:
            m32 = model(batch.inputs).detection.float()
            with autocast_context("bf16", cpu):
                m16 = model(batch.inputs).detection.float()
            l32 = torch.logit(m32[:, 0].double(), eps=1e-12)
            logit_diffs.append((l32 - torch.logit(m16[:, 0].double(), eps=1e-12)).abs().amax(dim=(1, 2)))
            fp32_logits.append(l32)
            d32 = decode_detections(m32, cfg.targets, threshold=DECODE_THRESHOLD)
            d16 = decode_detections(m16, cfg.targets, threshold=DECODE_THRESHOLD)
            for f in range(len(d32)):
                frames += 1
                f32, f16 = d32.frame(f), d16.frame(f)
                for t in thresholds:
                    x, y = _above(f32, t), _above(f16, t)
                    pairs, lone32, lone16 = pair_detections(x, y)
                    c = counts[t]
                    c["fp32"] += x.num_detections
                    c["bf16"] += y.num_detections
                    c["fp32_unpaired"] += len(lone32)
                    c["bf16_unpaired"] += len(lone16)
                    c["frames_same"] += not lone32 and not lone16
                    if t == DECODE_THRESHOLD:
                        for i, j in pairs:
                            d_score = max(d_score, abs(float(x.score[i] - y.score[j])))
                            d_range = max(d_range, abs(float(x.range_m[i] - y.range_m[j])))
                            d_az = max(d_az, abs(float(x.azimuth_deg[i] - y.azimuth_deg[j])))
    per_frame = torch.cat(logit_diffs)
    worst = float(per_frame.max())
    in_band = int(sum(((l - band_logit).abs() <= worst).sum() for l in fp32_logits))
    with open("/proc/loadavg") as f:
        load = f.read().split()[:3]
    print(json.dumps({
        "run": str(a.run), "split": a.split, "model": cfg.name, "cpu": cpu_model(),
        "native_bf16": cpu_has_native_bf16(), "threads": a.threads, "torch": torch.__version__,
        "loadavg": load, "frames": frames,
        "by_threshold": {f"{t:g}": c for t, c in counts.items()},
        "matched": {"pairs": counts[DECODE_THRESHOLD]["fp32"] - counts[DECODE_THRESHOLD]["fp32_unpaired"],
                    "max_score_diff": round(d_score, 5), "max_range_diff_m": round(d_range, 4),
                    "max_azimuth_diff_deg": round(d_az, 4)},
        "cells": {"max_logit_diff": round(worst, 4), "median_frame_max_logit_diff": round(float(per_frame.median()), 4),
                  "cells_in_band": in_band, "cells": int(sum(l.numel() for l in fp32_logits))},
    }, indent=1))


if __name__ == "__main__":
    main()
