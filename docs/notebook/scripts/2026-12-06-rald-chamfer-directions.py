"""Both directions of the Chamfer distance, per scene, for prediction folders (diagnostic)."""
# Run from the folder holding data/sim_colo6 and the prediction folders: python this.py PRED_DIR ...
import sys
import numpy as np
from scipy.spatial import cKDTree
from radarpc.data.coloradar import ColoRadar

ds = ColoRadar("data/sim_colo6", "test", cube_size=None, every=4)
folders = sys.argv[1:]
rows = {}
for i in range(0, len(ds), 2):                                 # every other scored frame: 50 frames
    k, ri, li = ds.index[i]
    run = ds.runs[k]
    gt = ds.lidar_points(i)
    for f in folders:
        p = np.load(f"{f}/{run.name}/{ri:06d}.npy")
        if len(p) == 0:
            continue
        acc = cKDTree(gt).query(p, workers=1)[0].mean()        # predicted -> truth
        comp = cKDTree(p).query(gt, workers=1)[0].mean()       # truth -> predicted
        rows.setdefault((f, run.scene), []).append((acc, comp, len(p)))
for (f, scene), v in sorted(rows.items()):
    a = np.array(v)
    print(f"{f:32s} {scene:10s} pred->truth {a[:,0].mean():.3f}  truth->pred {a[:,1].mean():.3f}  points {a[:,2].mean():.0f}")
