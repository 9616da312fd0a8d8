"""How large a difference between two RaLD-s arms is the frames' doing: per-frame CD and EMD of two
prediction folders on the same frames (their metrics.json, written by `radarpc evaluate-points` and by
`radarpc experiment rald-ablation`), the mean of the paired differences B - A overall and per scene, and
a 95 % bootstrap interval of that mean over frames (10,000 resamples of the frames, seed 0).
The interval covers the choice of test frames only, not the training seed (configs/rald/studies/seeds.yaml).
    python this.py PREDS_A PREDS_B [PREDS_B2 ...]      # prints JSON, one entry per B
"""
import json
import sys
from pathlib import Path

import numpy as np


def frames(folder):
    rows = json.loads((Path(folder) / "metrics.json").read_text())["frames"]
    return {(r["run"], r["frame"]): r for r in rows}


def paired(a, b, metric, scene=None):
    keys = sorted(k for k in a.keys() & b.keys() if scene is None or a[k]["scene"] == scene)
    d = np.array([b[k][metric] - a[k][metric] for k in keys])
    boot = np.random.default_rng(0).choice(d, size=(10_000, len(d))).mean(axis=1)
    lo, hi = np.quantile(boot, [0.025, 0.975])
    return {"frames": len(d), "mean_b_minus_a": round(float(d.mean()), 4),
            "ci95": [round(float(lo), 4), round(float(hi), 4)], "b_better_frames": int((d < 0).sum())}


a = frames(sys.argv[1])
out = []
for other in sys.argv[2:]:
    b = frames(other)
    if a.keys() != b.keys():
        sys.exit(f"{other}: scored on other frames than {sys.argv[1]} ({len(a.keys() ^ b.keys())} differ)")
    scenes = sorted({r["scene"] for r in a.values()})
    out.append({"a": sys.argv[1], "b": other,
                **{m: {"all": paired(a, b, m), **{s: paired(a, b, m, s) for s in scenes}} for m in ("chamfer", "emd")}})
print(json.dumps(out, indent=1))
