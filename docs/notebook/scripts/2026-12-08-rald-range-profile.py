"""Where the points are: range profile and both Chamfer directions per scene (diagnostic).

Run from the folder holding data/sim_colo6 and the prediction folders:
    python this.py PRED_DIR ...
Prints, for the LiDAR truth and each folder, per scene: the median range of the points, the fraction
beyond 10 m, and (for predictions) the two directions of the Chamfer distance; every other scored
test frame (50 frames).
"""
import sys

import numpy as np
from radarpc.data.coloradar import ColoRadar
from radarpc.eval.pointsets import ChamferTarget

ds = ColoRadar("data/sim_colo6", "test", cube_size=None, every=4)
folders = sys.argv[1:]
rows = {}
for i in range(0, len(ds), 2):
    k, ri, li = ds.index[i]
    run = ds.runs[k]
    gt = ds.lidar_points(i)
    r = np.linalg.norm(gt, axis=1)
    rows.setdefault(("truth", run.scene), []).append((np.median(r), (r > 10).mean(), np.nan, np.nan, len(gt)))
    target = ChamferTarget(gt, workers=1)
    for f in folders:
        p = np.load(f"{f}/{run.name}/{ri:06d}.npy")
        if len(p) == 0:
            continue
        r = np.linalg.norm(p, axis=1)
        acc, comp = target.directions(p)                        # predicted -> truth, truth -> predicted
        rows.setdefault((f, run.scene), []).append((np.median(r), (r > 10).mean(), acc, comp, len(p)))
for (f, scene), v in sorted(rows.items(), key=lambda kv: (kv[0][1], kv[0][0])):
    a = np.array(v)
    print(f"{scene:10s} {f:36s} median range {a[:,0].mean():5.2f} m  beyond 10 m {a[:,1].mean():.3f}  "
          f"pred->truth {a[:,2].mean():.3f}  truth->pred {a[:,3].mean():.3f}  points {a[:,4].mean():.0f}")
