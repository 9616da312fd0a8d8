"""Does RaLD-s use the radar? Each test frame generated from its own radar cube and from the cube of
a frame of another scene (the next scene's frame at the same position), decoded as Table 1 decodes
(500,000 random queries, no guide, no refinement); CD of both against the frame's own LiDAR truth.
Run from the folder holding runs/ and data/:  python this.py [STAGE-2 RUN]"""
import sys

import numpy as np, torch
from radarpc.config import load_yaml
from radarpc.data.coloradar import ColoRadar
from radarpc.eval.pointsets import chamfer_distance
from radarpc.experiments.rald.generation import GenerateConfig, model_input
from radarpc.experiments.rald.runs import load_rald
from radarpc.rald.generate import generate_cloud

torch.set_num_threads(1)
run = load_rald(sys.argv[1] if len(sys.argv) > 1 else "runs/rald-gen/stage2/rald-s-b7c52f5b0d")
cfg = load_yaml(GenerateConfig, "configs/rald/generate-table1-decoding.yaml").generation
ds = ColoRadar("data/sim_colo6", "test", cube_size=None, every=4)
to_input = model_input(run)
mirror = run.ae_config.data.mirror_azimuth
n, res = len(ds), {}
for i in range(0, n, 5):                                            # 20 frames, 5 a scene
    j = (i + n // 4) % n                                            # the same position in the next scene's run
    truth = ds.lidar_points(i)
    scene, other = ds.runs[ds.index[i][0]].scene, ds.runs[ds.index[j][0]].scene
    for label, src in (("own radar", i), ("another scene's radar", j)):
        cloud = generate_cloud(run.ae, run.dit, to_input(ds.cube(src)), np.zeros((0, 3), np.float32), cfg, seed=1000 + i,
                               grid=run.grid, mirror_azimuth=mirror)
        cd = chamfer_distance(cloud.points, truth) if len(cloud.points) else float("nan")
        res.setdefault((scene, label), []).append(cd)
    print(scene, other, [round(res[(scene, l)][-1], 3) for l in ("own radar", "another scene's radar")], flush=True)
for (scene, label), v in sorted(res.items()):
    print(f"{scene:10s} {label:24s} CD mean {np.nanmean(v):.3f} over {len(v)} frames")
