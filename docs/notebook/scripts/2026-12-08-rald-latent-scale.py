"""How large a stage-1 run's latents are, the scale stage 2's training noise is drawn against: over
every k-th training frame of a ColoRadar root, the standard deviation of the posterior sample z (all
entries), the mean posterior sigma, and the between-frame standard deviation of the posterior mean
(per latent entry across frames, then the root mean square over entries: how much a frame's latents
tell it apart from the others, what the radar must decide). EDM's sigma_data is 1 in rald-dit-s.
    python this.py AE_RUN [AE_RUN ...] --data ROOT [--every 20]      # prints JSON, one entry per run
"""
import argparse
import json

import torch

from radarpc.data.coloradar import ColoRadar
from radarpc.experiments.rald.generation import encoder_input
from radarpc.experiments.rald.runs import load_rald_ae

parser = argparse.ArgumentParser()
parser.add_argument("runs", nargs="+")
parser.add_argument("--data", required=True)
parser.add_argument("--every", type=int, default=20)
args = parser.parse_args()

frames = ColoRadar(args.data, split="train", every=args.every, cube_size=None)
out = []
for run_dir in args.runs:
    run = load_rald_ae(run_dir)
    to_input = encoder_input(run)
    gen = torch.Generator().manual_seed(0)
    means, zs, sigmas = [], [], []
    with torch.no_grad():
        for i in range(len(frames)):
            points = to_input(frames.lidar_points(i), gen)[None]                # (1, N, 3), no radar read
            mean, logvar = run.ae.encode(points)                                # (1, M, D) each
            means.append(mean[0].double())
            sigmas.append(torch.exp(0.5 * logvar[0]).double())
            zs.append(run.ae.sample(mean, logvar, torch.randn(mean.shape, generator=gen))[0].double())
    means, zs, sigmas = torch.stack(means), torch.stack(zs), torch.stack(sigmas)   # (F, M, D)
    out.append({"run": run_dir, "frames": len(frames),
                "z_std": round(zs.std().item(), 4),
                "posterior_sigma_mean": round(sigmas.mean().item(), 4),
                "between_frame_std_of_mean": round(means.std(dim=0).pow(2).mean().sqrt().item(), 4)})
print(json.dumps(out, indent=1))
